"""The service under load: the real API and a worker training a job, while many clients poll, upload and stream.

Starts everything on loopback from scratch: a throwaway PostgreSQL database (127.0.0.1:5432, user postgres), a private
Redis queue (127.0.0.1:6379), `drop api` (uvicorn) and one `drop worker` as subprocesses. It makes a token with
`drop token create`, uploads a small real hopper dataset and starts a long `cpu`-preset job on it. Once the worker
trains, for --seconds: --clients clients poll four read endpoints (wrk connections, spread evenly over the endpoints)
back to back, or --rate times a second each; --uploads clients upload --upload-mb MB D4RL-layout files one after
another (each must answer 201 and then be readable with GET); and --sse clients stream the job's events. It records
latency percentiles, counts and errors per endpoint, upload throughput, the events' delay from creation to arrival,
the API process's peak RSS and the job's fate (still running or succeeded, never failed or lost). Everything it
started is removed at the end, Ctrl-C included. Before any of it, the ceiling: `GET /healthz` against
`GET /v1/jobs/{id}` with wrk, the API alone.

    .venv/bin/python bench/service_load.py [--seconds 60] [--clients 50] [--uploads 5] [--upload-mb 100] [--sse 3]
    make bench-load                                   # the defaults
    .venv/bin/python bench/service_load.py --clients 5 --uploads 1 --upload-mb 10 --seconds 10   # a quick look

Writes bench/results/service_load.json and .md. The pollers are wrk (C), so their CPU use is small; the uploads and
the event streams are this process's asyncio clients, on the same cores as the service.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from contextlib import ExitStack, contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

import httpx
import numpy as np
import redis

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the service tests' helpers: throwaway database, worker process, settings as env

from kernel.settings import Settings  # noqa: E402
from tests.service.backends import REDIS_URL, database  # noqa: E402
from tests.service.processes import (  # noqa: E402
    free_port,
    kill_group,
    settings_env,
    start_worker,
    wait_for_line,
    wait_ready,
)

MB = 1_000_000
# Long enough to outlast any benchmark, small enough that epochs (and so events) come every few seconds.
JOB_OVERRIDES = {"epochs": 100_000, "steps_per_epoch": 100, "eval_every": 5, "eval_episodes": 1,
                 "checkpoint_every": 5, "log_every": 50, "dynamics.max_epochs": 5, "rollout.batch_size": 1000,
                 "dice.pretrain_steps": 50, "dice.steps_per_epoch": 50}
JOB_OK = {"running", "succeeded"}
NOTABLE = re.compile(r'WARNING|ERROR|CRITICAL|Traceback|Error:|"level": "(warning|error|critical)"')


# ------------------------------------------------------------------------------------------------ data
def make_files(folder: Path, upload_mb: float) -> tuple[Path, Path]:
    """A small real hopper dataset to train on, and an upload of `upload_mb` MB: those rows tiled, uncompressed."""
    from drop_engine.collect import collect_transitions, random_policy
    from drop_engine.data import load_dataset, save_hdf5

    rows = collect_transitions("hopper", random_policy(3, 0), 5000, seed=0)
    attrs = {"env_name": "Hopper-v4"}
    train = folder / "hopper-random.hdf5"
    save_hdf5(train, rows, attrs)
    per_row = sum(a[0].nbytes for a in rows.values())
    index = np.arange(int(upload_mb * MB) // per_row) % len(rows["observations"])
    upload = folder / "upload.hdf5"
    save_hdf5(upload, {k: a[index] for k, a in rows.items()}, attrs, compress=False)
    load_dataset(upload, env="hopper")  # the validator must accept it, or the benchmark measures refusals
    return train, upload


# ------------------------------------------------------------------------------------------------ the service
# `drop api` with the request observation (request id, HTTP metrics, access line) taken out: the ceiling's baseline
# for what observing costs. One process only: uvicorn then serves in the process that patched the app.
_RUN_DROP = "sys.argv[0] = 'drop'; from app.cli import main; main()"
UNOBSERVED_NAME = "this code, no request observation"
UNOBSERVED = f"import sys, app.main; app.main.ObserveRequests = lambda inner: inner; {_RUN_DROP}"
# The same with uvicorn's own access log in its default text format, as the API logged before the observation and
# the JSON logs: what the logging change costs against the service it replaced.
UVICORN_LOG_NAME = "no request observation, uvicorn's access log"
UVICORN_LOG = ("import sys, uvicorn.config, app.main, app.cli as cli; app.main.ObserveRequests = lambda inner: inner; "
               "app.main.configure = lambda *a, **k: None; options = cli._uvicorn_options; "
               "cli._uvicorn_options = lambda *a: {**options(*a), 'access_log': True, "
               f"'log_config': uvicorn.config.LOGGING_CONFIG}}; {_RUN_DROP}")


def api_command(repo: Path, port: int, workers: int, code: str | None = None) -> list[str]:
    """`drop api` from `repo` with `workers` processes, or `code` run as `python -c` in its place; a checkout from
    before `--workers` existed runs one anyway."""
    start = ["-m", "app.cli"] if code is None else ["-c", code]
    command = [sys.executable, *start, "api", "--host", "127.0.0.1", "--port", str(port)]
    return command + (["--workers", str(workers)] if "--workers" in (repo / "app/cli.py").read_text() else [])


@contextmanager
def service(folder: Path, upload_bytes: int, repo: Path = REPO,
            api_workers: int = 1) -> Iterator[tuple[str, str, subprocess.Popen, subprocess.Popen]]:
    """(API url, token, API process, worker process) on a fresh database and queue, the service's code from `repo`;
    all removed afterwards."""
    with database() as url:
        queue = f"drop-bench-{secrets.token_hex(4)}"
        # Quotas far above what the benchmark sends, so none of its own traffic is refused.
        settings = Settings(data_dir=folder / "data", database_url=url, broker_url=REDIS_URL, queue=queue,
                            max_upload_bytes=max(2 * 1024**3, 2 * upload_bytes), max_stored_bytes_per_owner=2**50,
                            max_active_jobs_per_owner=10_000, max_streams_per_owner=10_000,
                            max_uploads_per_owner=10_000, worker_threads=1, max_job_sac_updates=10**9,
                            max_job_metric_rows=10**9)
        env = settings_env(settings)
        drop = [sys.executable, "-m", "app.cli"]
        try:
            subprocess.run([*drop, "db", "upgrade"], cwd=repo, env=env, check=True, capture_output=True)
            token = subprocess.run([*drop, "token", "create", "--name", "bench-load"], cwd=repo, env=env, check=True,
                                   capture_output=True, text=True).stdout.strip()
            port = free_port()
            log = folder / "api.log"
            with log.open("ab") as out:
                api = subprocess.Popen(api_command(repo, port, api_workers), cwd=repo, env=env,
                                       stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
            try:
                wait_for_line(log, "Application startup complete", api, 120)
                worker = start_worker(settings, folder / "worker.log", repo)
                try:
                    yield f"http://127.0.0.1:{port}", token, api, worker
                finally:
                    kill_group(worker)
            finally:
                kill_group(api)
        finally:
            drop_queue(queue)


def drop_queue(queue: str) -> None:
    """Remove a bench run's Celery queue keys, so runs leave nothing in the shared Redis."""
    client = redis.Redis.from_url(REDIS_URL)
    for key in client.scan_iter(f"{queue}*"):
        client.delete(key)


@contextmanager
def idle_api(folder: Path, repo: Path, extra_env: dict[str, str], workers: int,
             code: str | None = None) -> Iterator[tuple[str, str, str, int]]:
    """(API url, token, a job's path, the API's pid) of a `drop api` from `repo` with no worker at all, on a database
    of its own holding one queued job: the API's own ceiling, nothing else running."""
    from tests.service.datasets import tiny_npz

    folder.mkdir(parents=True)
    with database() as url:
        settings = Settings(data_dir=folder / "data", database_url=url, broker_url=REDIS_URL,
                            queue=f"drop-bench-idle-{secrets.token_hex(4)}")
        env = {**settings_env(settings), **extra_env}
        drop = [sys.executable, "-m", "app.cli"]
        try:
            subprocess.run([*drop, "db", "upgrade"], cwd=repo, env=env, check=True, capture_output=True)
            token = subprocess.run([*drop, "token", "create", "--name", "bench-ceiling"], cwd=repo, env=env,
                                   check=True, capture_output=True, text=True).stdout.strip()
            port = free_port()
            with (folder / "api.log").open("ab") as out:
                api = subprocess.Popen(api_command(repo, port, workers, code), cwd=repo, env=env, stdout=out,
                                       stderr=subprocess.STDOUT, start_new_session=True)
            try:
                base = f"http://127.0.0.1:{port}"
                with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=60) as http:
                    wait_ready(http, api, folder / "api.log", 120)  # a quiet variant logs no startup line
                    ds = http.post("/v1/datasets", content=tiny_npz(0)).raise_for_status().json()
                    job = http.post("/v1/jobs", json={"dataset_id": ds["id"], "env": "hopper", "preset": "smoke"})
                yield base, token, f"/v1/jobs/{job.raise_for_status().json()['id']}", api.pid
            finally:
                kill_group(api)
        finally:
            drop_queue(settings.queue)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time so far of a process and its live descendants (`--workers N`'s API processes)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    own = sum(int(f) for f in fields[11:13]) / os.sysconf("SC_CLK_TCK")
    kids = [int(c) for task in Path(f"/proc/{pid}/task").iterdir() for c in (task / "children").read_text().split()]
    return own + sum(cpu_seconds(kid) for kid in kids)


def postgres_cpu_seconds() -> float:
    """User + system CPU time so far of every PostgreSQL process on the machine: the server the API reads from, and
    approximate (another cluster's processes count too; a backend that exits meanwhile takes its time with it)."""
    total = 0.0
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and (proc / "comm").read_text().strip() == "postgres":
                total += sum(int(f) for f in (proc / "stat").read_text().rsplit(")", 1)[1].split()[11:13])
        except OSError:  # gone meanwhile
            pass
    return total / os.sysconf("SC_CLK_TCK")


def wrk(url: str, token: str, seconds: float, pid: int, connections: int = 16) -> tuple[float, int, float, float]:
    """(requests per second, answers other than 2xx, the API's CPU µs per request, PostgreSQL's) of wrk's closed loop
    on one URL. CPU per request varies far less than throughput on a noisy machine, so it tells small costs apart."""
    cpu, db = cpu_seconds(pid), postgres_cpu_seconds()
    out = subprocess.run(["wrk", "-t1", f"-c{connections}", f"-d{seconds:g}s", "-H", f"Authorization: Bearer {token}",
                          url], check=True, capture_output=True, text=True).stdout
    cpu, db = cpu_seconds(pid) - cpu, postgres_cpu_seconds() - db
    bad = re.search(r"Non-2xx or 3xx responses: (\d+)", out)
    requests = max(int(re.search(r"(\d+) requests in", out).group(1)), 1)
    return (float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1)), int(bad.group(1)) if bad else 0,
            1e6 * cpu / requests, 1e6 * db / requests)


def ceiling(args, folder: Path) -> dict:
    """Requests per second of `GET /healthz` (the framework's own ceiling) and of `GET /v1/jobs/{id}` with auth, for
    each variant of the API, with no worker running; the same client (wrk) and number of API processes throughout.
    The measurements alternate in short rounds and each figure is the median of its rounds, so that a busy
    machine's drift falls on all of them alike."""
    if shutil.which("wrk") is None:
        raise SystemExit("the ceiling needs wrk (apt-get install wrk), or --ceiling-rounds 0")
    variants = [("this code", REPO, {}, None), ("this code, access log off", REPO, {"DROP_LOG_LEVEL": "WARNING"}, None)]
    if args.api_workers == 1:
        variants += [(UNOBSERVED_NAME, REPO, {}, UNOBSERVED), (UVICORN_LOG_NAME, REPO, {}, UVICORN_LOG)]
    if args.before_repo:
        variants.append(("before", args.before_repo, {}, None))
    with ExitStack() as stack:
        targets = []
        for i, (name, repo, extra, code) in enumerate(variants):
            base, token, job, pid = stack.enter_context(idle_api(folder / f"ceiling-{i}", repo, extra,
                                                                 args.api_workers, code))
            targets += [(name, "GET /healthz", base + "/healthz", token, pid),
                        (name, "GET /v1/jobs/{id}", base + job, token, pid)]
        runs: dict[tuple[str, str], list[tuple[float, int, float, float]]] = defaultdict(list)
        for r in range(args.ceiling_rounds):
            print(f"  ceiling round {r + 1}/{args.ceiling_rounds}", flush=True)
            for name, endpoint, url, token, pid in targets:
                runs[(name, endpoint)].append(wrk(url, token, args.ceiling_round_s, pid))
    table = {name: {endpoint: {"rps": round(float(np.median([r[0] for r in runs[(name, endpoint)]])), 1),
                               "cpu_us": round(float(np.median([r[2] for r in runs[(name, endpoint)]])), 1),
                               "db_cpu_us": round(float(np.median([r[3] for r in runs[(name, endpoint)]])), 1),
                               "rounds": runs[(name, endpoint)],
                               "errors": sum(r[1] for r in runs[(name, endpoint)])}
                    for endpoint in ("GET /healthz", "GET /v1/jobs/{id}")} for name, *_ in variants}
    for row in table.values():
        row["job_share_of_healthz"] = round(row["GET /v1/jobs/{id}"]["rps"] / row["GET /healthz"]["rps"], 3)
    return {"api_workers": args.api_workers, "rounds": args.ceiling_rounds, "round_s": args.ceiling_round_s,
            "connections": 16, "variants": table}


def notable_lines(log: Path, most: int = 40) -> list[str]:
    """The warnings, errors and tracebacks a server process logged: the server's side of any problem."""
    lines = [line for line in log.read_text(errors="replace").splitlines() if NOTABLE.search(line)]
    return lines[:most]


def rss_mb(pid: int, field: str) -> float:
    """VmRSS (now) or VmHWM (peak) of a process, in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024 / MB
    raise LookupError(field)


# ------------------------------------------------------------------------------------------------ the clients
class Recorder:
    """Latency and outcome of every request, per endpoint, and every unexpected outcome."""

    def __init__(self) -> None:
        self.latency: dict[str, list[float]] = defaultdict(list)
        self.statuses: dict[str, Counter] = defaultdict(Counter)
        self.problems: Counter = Counter()

    def problem(self, endpoint: str, what: str) -> None:
        self.problems[f"{endpoint}: {what}"] += 1

    def failed(self, endpoint: str, exc: Exception) -> None:
        """A request that got no answer, named by its innermost cause (httpx's own messages are often empty)."""
        root = exc
        while root.__context__ is not None:
            root = root.__context__
        self.problem(endpoint, f"{type(exc).__name__} ({type(root).__name__}: {str(root)[:120]})")

    async def call(self, endpoint: str, request) -> httpx.Response | None:
        start = time.perf_counter()
        try:
            response = await request
        except httpx.HTTPError as exc:
            self.latency[endpoint].append(time.perf_counter() - start)
            self.statuses[endpoint][type(exc).__name__] += 1
            self.failed(endpoint, exc)
            return None
        self.latency[endpoint].append(time.perf_counter() - start)
        self.statuses[endpoint][str(response.status_code)] += 1
        if not response.is_success:
            code = response.json().get("code", "") if "json" in response.headers.get("content-type", "") else ""
            self.problem(endpoint, f"{response.status_code} {code}".strip())
        return response

    def errors(self, endpoint: str) -> int:
        return sum(n for status, n in self.statuses[endpoint].items() if not status.startswith("2"))


# One wrk process per endpoint: wrk's `delay()` makes each connection a client that asks `rate` times a second (the
# think time between an answer and its next request), or back to back without it; `done()` prints the percentiles.
WRK_SCRIPT = """
local delay_ms = 0
function init(args) delay_ms = tonumber(args[1]) end
if tonumber(os.getenv("WRK_DELAY_MS") or "0") > 0 then
  function delay() return delay_ms end
end
function done(summary, latency, requests)
  local e = summary.errors
  io.write(string.format('{"requests": %d, "non_2xx": %d, "socket_errors": %d, "seconds": %.3f, "min": %.1f, '
    .. '"p50": %.1f, "p95": %.1f, "p99": %.1f, "max": %.1f}\\n', summary.requests, e.status,
    e.connect + e.read + e.write + e.timeout, summary.duration / 1e6, latency.min / 1e3, latency:percentile(50) / 1e3,
    latency:percentile(95) / 1e3, latency:percentile(99) / 1e3, latency.max / 1e3))
end
"""


async def poll_with_wrk(base: str, token: str, targets: list[tuple[str, str]], args, folder: Path) -> dict:
    """Per endpoint: requests, errors, per second and latency percentiles (ms) of args.clients connections in all,
    spread evenly over the endpoints, for args.seconds. The load comes from wrk (C), so the client's own CPU use is
    small next to the service's; a Python client on these cores saturated before the API did."""
    script = folder / "poll.lua"
    script.write_text(WRK_SCRIPT)
    delay_ms = round(1000 / args.rate) if args.rate else 0
    procs = []
    for n, (name, url) in enumerate(targets):
        connections = args.clients // len(targets) + (n < args.clients % len(targets))
        procs.append((name, await asyncio.create_subprocess_exec(
            "wrk", "-t1", f"-c{connections}", f"-d{args.seconds:g}s", "--timeout", "10s", "-s", str(script),
            "-H", f"Authorization: Bearer {token}", base + url, "--", str(delay_ms),
            env={**os.environ, "WRK_DELAY_MS": str(delay_ms)}, stdout=asyncio.subprocess.PIPE)))
    endpoints = {}
    for name, proc in procs:
        out, _ = await proc.communicate()
        r = json.loads(out.decode().strip().splitlines()[-1])
        errors = r["non_2xx"] + r["socket_errors"]
        endpoints[name] = {"requests": r["requests"], "errors": errors, "per_s": round(r["requests"] / r["seconds"], 1),
                           "statuses": {"2xx": r["requests"] - r["non_2xx"], "other": r["non_2xx"],
                                        "socket errors": r["socket_errors"]},
                           "latency_ms": {k: r[k] for k in ("min", "p50", "p95", "p99", "max")}}
    return endpoints


async def upload_loop(client: httpx.AsyncClient, path: Path, stop_at: float, rec: Recorder, out: list[dict]) -> None:
    """Upload the file again and again until the time is up; each must be a 201 whose dataset GET then returns."""
    size = path.stat().st_size
    while time.monotonic() < stop_at:
        sent: dict[str, float] = {}

        async def body():
            with path.open("rb") as fh:
                while chunk := fh.read(1 << 20):
                    yield chunk
            sent["at"] = time.perf_counter()  # noqa: B023 (awaited within this iteration, before `sent` is rebound)

        start = time.perf_counter()
        response = await rec.call("POST /v1/datasets", client.post(
            "/v1/datasets", params={"name": f"load-{len(out)}.hdf5"}, content=body(),
            headers={"Content-Type": "application/x-hdf5", "Content-Length": str(size)}, timeout=900))
        seconds = time.perf_counter() - start
        record = {"status": response.status_code if response is not None else None, "seconds": round(seconds, 3),
                  "send_s": round(sent.get("at", start + seconds) - start, 3), "mb_s": round(size / MB / seconds, 2)}
        out.append(record)
        if record["status"] != 201:
            continue
        record["dataset_id"] = response.json()["id"]
        check = await rec.call("GET /v1/datasets/{id} (after its upload)",
                               client.get(f"/v1/datasets/{record['dataset_id']}"))
        record["readable"] = (check is not None and check.status_code == 200
                              and check.json().get("size_bytes") == size)
        if not record["readable"]:
            rec.problem("POST /v1/datasets", f"dataset {record['dataset_id']} answered 201 but GET does not return it")


async def stream_events(client: httpx.AsyncClient, url: str, rec: Recorder, delays: list[float]) -> None:
    """Follow the job's event stream (reconnecting with Last-Event-ID) until cancelled; note each event's delay from
    its creation to its arrival here."""
    last, since = None, datetime.now(timezone.utc)  # events from before are replayed, not delivered late
    while True:
        headers = {"Accept": "text/event-stream", **({"Last-Event-ID": last} if last else {})}
        start = time.perf_counter()
        try:
            async with client.stream("GET", url, headers=headers, timeout=httpx.Timeout(60, read=None)) as response:
                rec.latency["GET /v1/jobs/{id}/events (SSE connect)"].append(time.perf_counter() - start)
                rec.statuses["GET /v1/jobs/{id}/events (SSE connect)"][str(response.status_code)] += 1
                if response.status_code != 200:
                    rec.problem("SSE", f"{response.status_code} on connect")
                    await asyncio.sleep(1)
                    continue
                async for line in response.aiter_lines():
                    if line == "event: end":  # the job finished: nothing more will come
                        return
                    if line.startswith("id: "):
                        last = line[4:]
                    elif line.startswith("data: ") and '"created_at"' in line:
                        created = datetime.fromisoformat(json.loads(line[6:])["created_at"])
                        if created >= since:
                            delays.append((datetime.now(timezone.utc) - created).total_seconds())
        except httpx.HTTPError as exc:
            rec.failed("SSE", exc)
            await asyncio.sleep(1)


async def wait_training(client: httpx.AsyncClient, job_id: str, timeout: float = 300) -> dict:
    """The job once its model is fitted and policy epochs (each with its events) have begun."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = (await client.get(f"/v1/jobs/{job_id}")).raise_for_status().json()
        if job["status"] == "running" and (job.get("progress") or {}).get("phase") == "train":
            return job
        if job["status"] not in ("queued", "running"):
            raise RuntimeError(f"job {job_id} is {job['status']} before the load started: {job.get('error')}")
        await asyncio.sleep(0.5)
    raise RuntimeError(f"job {job_id} did not start within {timeout:.0f} s")


def percentiles(values: list[float], scale: float = 1000.0) -> dict:
    if not values:
        return {}
    p = np.percentile(np.asarray(values) * scale, [0, 50, 95, 99, 100]).round(1).tolist()
    return dict(zip(("min", "p50", "p95", "p99", "max"), p))


async def run_load(args, base: str, token: str, api: subprocess.Popen, worker: subprocess.Popen,
                   train: Path, upload: Path) -> dict:
    total = args.clients + args.uploads + args.sse + 4
    limits = httpx.Limits(max_connections=total, max_keepalive_connections=total)
    async with httpx.AsyncClient(base_url=base, headers={"Authorization": f"Bearer {token}"}, limits=limits,
                                 timeout=60) as client:
        response = await client.post("/v1/datasets", params={"name": train.name}, content=train.read_bytes(),
                                     headers={"Content-Type": "application/x-hdf5"})
        dataset_id = response.raise_for_status().json()["id"]
        response = await client.post("/v1/jobs", json={"dataset_id": dataset_id, "algorithm": "drop", "preset": "cpu",
                                                       "seed": 0, "overrides": JOB_OVERRIDES})
        job_id = response.raise_for_status().json()["id"]
        job_start = await wait_training(client, job_id)
        seen = (await client.get(f"/v1/jobs/{job_id}/events", params={"limit": 1000})).json()["data"]
        recent = seen[-1]["id"] if seen else 0  # pollers ask for what is new since, as a client following a job does
        print(f"job {job_id} at {progress(job_start['progress'])}; load for {args.seconds:.0f} s", flush=True)

        rec, uploads, delays = Recorder(), [], []
        rss_start, load_start = rss_mb(api.pid, "VmRSS"), os.getloadavg()
        targets = [("GET /v1/jobs/{id}", f"/v1/jobs/{job_id}"),
                   ("GET /v1/jobs/{id}/events?after=", f"/v1/jobs/{job_id}/events?after={recent}"),
                   ("GET /v1/jobs", "/v1/jobs"),
                   ("GET /v1/datasets/{id}", f"/v1/datasets/{dataset_id}")]
        streams = [asyncio.create_task(stream_events(client, f"/v1/jobs/{job_id}/events", rec, delays))
                   for _ in range(args.sse)]
        connects = rec.latency["GET /v1/jobs/{id}/events (SSE connect)"]
        for _ in range(300):  # the load starts once the streams are open: their connects are measured on their own
            if len(connects) >= args.sse:
                break
            await asyncio.sleep(0.1)
        began = time.monotonic()
        stop_at = began + args.seconds
        pollers = asyncio.create_task(poll_with_wrk(base, token, targets, args, train.parent))
        bounded = [pollers, *(asyncio.create_task(upload_loop(client, upload, stop_at, rec, uploads))
                    for _ in range(args.uploads))]
        try:
            while not all(t.done() for t in bounded):
                await asyncio.wait(bounded, timeout=10)
                print(f"  {time.monotonic() - began:5.0f} s: {sum(rec.problems.values())} problems, "
                      f"{len(uploads)} uploads done", flush=True)
        finally:  # the streams never end by themselves, and on Ctrl-C nothing may outlive the client
            for t in streams + bounded:
                t.cancel()
            outcomes = await asyncio.gather(*bounded, *streams, return_exceptions=True)
        uploads_s = time.monotonic() - began
        for outcome in outcomes:
            if isinstance(outcome, Exception):
                rec.failed("client crashed", outcome)
        polled = pollers.result() if pollers.done() and not pollers.cancelled() and not pollers.exception() else {}
        for name, endpoint in polled.items():
            if endpoint["errors"]:
                rec.problem(name, f"{endpoint['errors']} errors ({endpoint['statuses']})")

        job_end = (await client.get(f"/v1/jobs/{job_id}")).json()
        if job_end["status"] not in JOB_OK:
            rec.problem("job", f"ended {job_end['status']}: {job_end.get('error')}")
        elif job_end["status"] == "running" and job_end.get("progress") == job_start["progress"]:
            rec.problem("job", "made no progress during the load")
        rss_peak = rss_mb(api.pid, "VmHWM") if api.poll() is None else None
        for name, proc in (("API", api), ("worker", worker)):
            if proc.poll() is not None:
                rec.problem(name, f"process exited with {proc.returncode}")
        return report(args, rec, polled, uploads, delays, upload.stat().st_size, uploads_s, load_start,
                      {"start": round(rss_start, 1), "peak": rss_peak and round(rss_peak, 1)},
                      {"id": job_id, "status_end": job_end["status"], "progress_start": job_start["progress"],
                       "progress_end": job_end.get("progress"), "overrides": JOB_OVERRIDES})


# ------------------------------------------------------------------------------------------------ results
def stamp() -> dict:
    """When and on which commit a result was measured."""
    return {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "commit": subprocess.run(["git", "describe", "--always", "--dirty"], cwd=REPO, capture_output=True,
                                     text=True).stdout.strip()}


def report(args, rec: Recorder, polled: dict, uploads: list[dict], delays: list[float], upload_bytes: int,
           uploads_s: float, load_start: tuple, rss: dict, job: dict) -> dict:
    """The polled endpoints as wrk measured them, and the SSE connects and uploads as this client did."""
    endpoints = dict(polled)
    for name in rec.latency:
        endpoints[name] = {"requests": len(rec.latency[name]), "errors": rec.errors(name),
                           "per_s": round(len(rec.latency[name]) / (uploads_s if name.startswith("POST") else
                                                                    args.seconds), 1),
                           "statuses": dict(rec.statuses[name]), "latency_ms": percentiles(rec.latency[name])}
    endpoints = dict(sorted(endpoints.items()))
    ok = [u for u in uploads if u["status"] == 201 and u.get("readable")]
    return {
        **stamp(),
        "settings": {"seconds": args.seconds, "clients": args.clients, "uploads": args.uploads,
                     "upload_mb": args.upload_mb, "sse": args.sse, "rate": args.rate, "api_workers": args.api_workers,
                     "service": "this code" if args.service_repo == REPO else str(args.service_repo)},
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "loadavg_start": load_start,
                    "loadavg_end": os.getloadavg(), "note": args.note},
        "endpoints": endpoints,
        "uploads": {"file_mb": round(upload_bytes / MB, 1), "count": len(uploads), "ok": len(ok),
                    "seconds": round(uploads_s, 1), "total_mb_s": round(len(ok) * upload_bytes / MB / uploads_s, 2),
                    "each_mb_s": percentiles([u["mb_s"] for u in ok], 1.0),
                    "send_s": percentiles([u["send_s"] for u in ok], 1.0), "all": uploads},
        "sse": {"clients": args.sse, "events": len(delays), "delay_ms": percentiles(delays)},
        "api_rss_mb": rss,
        "job": job,
        "problems": dict(rec.problems.most_common()),
    }


def progress(p: dict | None) -> str:
    return f"{p['phase']} epoch {p['epoch']} step {p['step']}/{p['total']}" if p else "-"


def ceiling_markdown(c: dict) -> list[str]:
    lines = [f"## Ceiling: the API alone, no worker ({c['api_workers']} API process(es), wrk with {c['connections']} "
             f"connections, the median of {c['rounds']} alternating rounds of {c['round_s']:g} s)", "",
             "| service | `GET /healthz` req/s | `GET /v1/jobs/{id}` req/s (auth, PostgreSQL) | share of healthz | "
             "API CPU µs per healthz | per job read | PostgreSQL CPU µs per job read | errors |",
             "|---|---|---|---|---|---|---|---|"]
    for name, row in c["variants"].items():
        health, job = row["GET /healthz"], row["GET /v1/jobs/{id}"]
        lines.append(f"| {name} | {health['rps']} | {job['rps']} | {row['job_share_of_healthz']:.0%} | "
                     f"{health['cpu_us']} | {job['cpu_us']} | {job.get('db_cpu_us', '-')} | "
                     f"{health['errors'] + job['errors']} |")
    table, here = c["variants"], c["variants"]["this code"]

    def cost(base: dict, what: str) -> str:
        """What `here` spends beyond `base`, as a share of its throughput and of its CPU per request."""
        return "; ".join(f"{e.split()[1]}: {1 - here[e]['rps'] / base[e]['rps']:.1%} of the throughput, "
                         f"{1 - base[e]['cpu_us'] / here[e]['cpu_us']:.1%} of the API's CPU per request"
                         for e in ("GET /healthz", "GET /v1/jobs/{id}")) + f" ({what})."

    lines.append("")
    if "this code, access log off" in table:
        lines.append("The access log line costs " + cost(table["this code, access log off"],
                                                         "this code against itself with DROP_LOG_LEVEL=WARNING"))
    if UNOBSERVED_NAME in table:
        lines.append("Observing requests (request id, HTTP metrics, access line) costs " + cost(
            table[UNOBSERVED_NAME], "this code against itself with the observing middleware taken out"))
    if UVICORN_LOG_NAME in table:
        lines.append("Against uvicorn's own access log with no observation, as the API logged before, observing costs "
                     + cost(table[UVICORN_LOG_NAME], "a negative share is a saving"))
    if "before" in table:
        lines.append(f"Against the code before, healthz runs at "
                     f"{here['GET /healthz']['rps'] / table['before']['GET /healthz']['rps']:.0%} and the job read at "
                     f"{here['GET /v1/jobs/{id}']['rps'] / table['before']['GET /v1/jobs/{id}']['rps']:.0%}.")
    return lines


def markdown(r: dict) -> str:
    s, m, u = r["settings"], r["machine"], r["uploads"]
    load = " / ".join(f"{x:.2f}" for x in m["loadavg_start"])
    lines = [
        f"# Service under load ({r['date']}, {r['commit']})", "",
        f"Service: {s['service']}. {s['clients']} clients polling for {s['seconds']:.0f} s "
        + (f"at {s['rate']:g} requests/s each ({s['clients'] * s['rate']:g}/s offered)" if s["rate"] else
           "back to back (the closed-loop maximum)")
        + f", {s['uploads']} clients uploading {u['file_mb']:.0f} MB datasets one after another, {s['sse']} SSE "
        f"streams of the job's events; `drop api` with {s['api_workers']} process(es), one `drop worker` training a "
        "`cpu`-preset DROP job, PostgreSQL and Redis on loopback.",
        "",
        f"Machine: {m['cpus']} cores, {m['platform']}; load average (1/5/15 min) at start {load}. The clients run on "
        "the same cores, so their own CPU use is inside these latencies." + (f" {m['note']}" if m["note"] else ""),
        "",
        "| endpoint | requests | per s | errors | p50 ms | p95 ms | p99 ms | max ms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, e in r["endpoints"].items():
        p = e["latency_ms"]
        lines.append(f"| `{name}` | {e['requests']} | {e['per_s']} | {e['errors']} | {p['p50']} | {p['p95']} | "
                     f"{p['p99']} | {p['max']} |")
    each, send = u["each_mb_s"] or {}, u["send_s"] or {}
    sse, job, rss = r["sse"], r["job"], r["api_rss_mb"]
    lines += [
        "",
        f"Uploads: {u['ok']} of {u['count']} answered 201 and were then returned by GET; each {u['file_mb']:.0f} MB "
        f"at {each.get('p50', '-')} MB/s (median; slowest {each.get('min', '-')}, fastest {each.get('max', '-')}), "
        f"{u['total_mb_s']} MB/s in total over {u['seconds']:.0f} s; sending the body took a median "
        f"{send.get('p50', '-')} s of each (the rest is validation and saving).",
        f"SSE: {sse['events']} new events delivered to {sse['clients']} streams, delay from creation to arrival "
        f"p50 {sse['delay_ms'].get('p50', '-')} ms, p95 {sse['delay_ms'].get('p95', '-')} ms, p99 "
        f"{sse['delay_ms'].get('p99', '-')} ms.",
        f"API process RSS: {rss['start']} MB when the load began, peak {rss['peak']} MB (VmHWM).",
        f"Job: {job['status_end']} at the end; it went from {progress(job['progress_start'])} to "
        f"{progress(job['progress_end'])} during the load.",
        "",
        "Problems: " + ("none." if not r["problems"] else ""),
    ]
    lines += [f"- {what}: {n}" for what, n in r["problems"].items()]
    if r.get("ceiling"):
        lines += ["", *ceiling_markdown(r["ceiling"])]
    logged = [f"- {name}: `{line}`" for name, found in r["server_log"].items() for line in found]
    if logged:
        lines += ["", "Warnings and errors the server processes logged:", *logged]
    return "\n".join(lines) + "\n"


def write_ceiling(args, limits: dict) -> int:
    """`--ceiling-only`: the ceiling's table, with the date, commit and machine it was measured on."""
    result = {**stamp(), "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "note": args.note},
              "ceiling": limits}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
    m = result["machine"]
    text = "\n".join([f"# Ceiling of the API ({result['date']}, {result['commit']})", "",
                      f"Machine: {m['cpus']} cores, {m['platform']}." + (f" {m['note']}" if m["note"] else ""), "",
                      *ceiling_markdown(limits)]) + "\n"
    (args.out / f"{args.name}.md").write_text(text)
    print(text)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="how long the load lasts")
    parser.add_argument("--clients", type=int, default=50, help="concurrent polling clients")
    parser.add_argument("--uploads", type=int, default=5, help="concurrent uploading clients")
    parser.add_argument("--upload-mb", type=float, default=100.0, help="size of each uploaded file (MB)")
    parser.add_argument("--sse", type=int, default=3, help="clients streaming the job's events")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="requests per second per polling client (an offered load); 0: back to back (the maximum)")
    parser.add_argument("--api-workers", type=int, default=1, help="`drop api --workers`")
    parser.add_argument("--service-repo", type=Path, default=REPO,
                        help="a checkout whose service runs the load (e.g. an older commit, for before figures)")
    parser.add_argument("--before-repo", type=Path, default=None,
                        help="a checkout measured beside this code in the ceiling (same run, alternating rounds)")
    parser.add_argument("--ceiling-rounds", type=int, default=4, help="0 skips the ceiling")
    parser.add_argument("--ceiling-round-s", type=float, default=3.0)
    parser.add_argument("--ceiling-only", action="store_true", help="measure the ceiling alone, no load after it")
    parser.add_argument("--name", default="service_load", help="results file stem in --out")
    parser.add_argument("--note", default="", help="a sentence about the machine for the markdown (background load)")
    parser.add_argument("--out", type=Path, default=REPO / "bench/results")
    args = parser.parse_args()
    if args.clients < 4:
        parser.error("--clients must be at least 4: one wrk connection per polled endpoint")
    for sig in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C or a kill cleans up, even when started in the background
        signal.signal(sig, signal.default_int_handler)

    with tempfile.TemporaryDirectory(prefix="drop-bench-load-") as tmp:
        folder = Path(tmp)
        print(f"making datasets in {folder}", flush=True)
        train, upload = make_files(folder, args.upload_mb)
        limits = ceiling(args, folder) if args.ceiling_rounds else None
        if args.ceiling_only:
            return write_ceiling(args, limits)
        print("starting PostgreSQL database, API and worker", flush=True)
        with service(folder, upload.stat().st_size, args.service_repo, args.api_workers) as (base, token, api, worker):
            result = asyncio.run(run_load(args, base, token, api, worker, train, upload))
            result["server_log"] = {name: notable_lines(folder / f"{name}.log") for name in ("api", "worker")}
        result["ceiling"] = limits
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
    text = markdown(result)
    (args.out / f"{args.name}.md").write_text(text)
    print(text)
    return 1 if result["problems"] else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        sys.exit("interrupted; the processes, database, Redis keys and temporary files it made are removed")
